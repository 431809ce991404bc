"""Run-level evaluation reports: the JSON-ready figures of ``metrics.json`` and the standard plots.

Shared by ``neb-slam eval`` and the run report of ``neb-slam run`` (:mod:`.run_report`).
"""

from __future__ import annotations

import json
from pathlib import Path


def merge_metrics(path: Path, new: dict) -> dict:
    """Update the JSON object in ``path`` (created when absent) with ``new``; returns the merged object."""
    from ..errors import DatasetError

    merged: dict = {}
    if path.is_file():
        try:
            merged = json.loads(path.read_text())
        except json.JSONDecodeError as exc:
            raise DatasetError(path, f"existing metrics file is not valid JSON ({exc}); fix or remove it") from None
        if not isinstance(merged, dict):
            raise DatasetError(path, "existing metrics file must hold a JSON object")
    merged.update(new)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(merged, indent=2, sort_keys=True) + "\n")
    return merged


def trajectory_metrics(
    est,
    gt,
    *,
    max_dt_s: float = 0.02,
    align: bool = True,
    rpe_delta_s: float = 1.0,
    est_source: Path | None = None,
    gt_source: Path | None = None,
):
    """ATE and RPE of trajectory ``est`` against ``gt`` (both :class:`~neb_slam_core.io.trajectory.Trajectory`).

    Returns ``(metrics, ate)``: the JSON-ready figures this command writes (``ate_rmse_cm``, ...,
    ``n_gt_poses``) and the :class:`~neb_slam_core.eval.trajectory_metrics.AteResult` (for plots and
    mesh alignment). Raises :class:`DatasetError` when fewer than 3 poses associate.
    """
    from .trajectory_metrics import associate_trajectories, compute_ate, compute_rpe

    pair = associate_trajectories(est, gt, max_dt_s, est_source=est_source, gt_source=gt_source)
    ate = compute_ate(pair, align=align)
    rpe = compute_rpe(pair, rpe_delta_s, "s")
    rpe_frame = compute_rpe(pair, 1, "frames")

    def cm(v: float | None) -> float | None:
        return None if v is None else v * 100.0

    metrics: dict = {
        "ate_rmse_cm": ate.rmse_cm,
        "ate_mean_cm": ate.mean_cm,
        "ate_median_cm": ate.median_cm,
        "ate_max_cm": ate.max_cm,
        "rpe_trans_cm": cm(rpe.trans_rmse_m),
        "rpe_rot_deg": rpe.rot_rmse_deg,
        "rpe_delta_s": rpe_delta_s,
        "rpe_frame_trans_cm": cm(rpe_frame.trans_rmse_m),
        "rpe_frame_rot_deg": rpe_frame.rot_rmse_deg,
        "n_poses": ate.n_matched,
        "n_est_poses": ate.n_est,
        "n_gt_poses": ate.n_gt,
    }
    return metrics, ate


def recon_metrics(recon) -> dict:
    """The JSON-ready figures of a :class:`~neb_slam_core.eval.recon.ReconResult`."""
    return {
        "accuracy_cm": recon.accuracy_cm,
        "completion_cm": recon.completion_cm,
        "completion_ratio_pct": recon.completion_ratio_pct,
        "depth_l1_cm": recon.depth_l1_cm,
        "completion_threshold_cm": recon.completion_threshold_cm,
        "recon_culled": recon.culled,
        "recon_points": recon.n_points,
        "recon_floor_cm": recon.sampling_floor_cm,
    }


def write_trajectory_plots(ate, out_dir: Path, loops=()) -> list[Path]:
    """``trajectory.png`` (with ``loops`` marked, see :func:`~neb_slam_core.eval.plots.plot_trajectory`)
    and ``ate_over_time.png`` of ``ate`` in ``out_dir``; returns their paths."""
    from .plots import plot_ate_over_time, plot_trajectory, save_figure

    return [
        save_figure(plot_trajectory(ate, loops=loops), out_dir / "trajectory.png"),
        save_figure(plot_ate_over_time(ate), out_dir / "ate_over_time.png"),
    ]


def evaluate_mesh_files(
    rec_path: Path,
    gt_mesh_path: Path,
    *,
    T_gt_rec=None,
    cull_poses=None,
    intrinsics=None,
    n_points: int = 200_000,
    threshold_cm: float = 5.0,
    depth_views: int = 1000,
    seed: int = 0,
):
    """Reconstruction metrics of the mesh file ``rec_path`` against ``gt_mesh_path``.

    Args:
        T_gt_rec: ``(4, 4)`` map of the reconstruction into the ground truth's frame (None: already there).
        cull_poses: ``(m, 4, 4)`` ground-truth camera poses to cull both meshes to (with ``intrinsics``);
            None compares the whole meshes.
        intrinsics: the recording camera (:class:`~neb_slam_core.types.Intrinsics`).

    Returns:
        :class:`~neb_slam_core.eval.recon.ReconResult`.
    """
    from dataclasses import replace

    from .recon import DepthL1Config, ReconConfig, evaluate_reconstruction, load_mesh

    rec_mesh = load_mesh(rec_path)
    gt_mesh = load_mesh(gt_mesh_path)
    if T_gt_rec is not None:
        rec_mesh = rec_mesh.copy()
        rec_mesh.apply_transform(T_gt_rec)
    config = ReconConfig(
        n_points=n_points,
        completion_threshold_m=threshold_cm / 100.0,
        seed=seed,
        depth_l1=replace(DepthL1Config(), n_views=depth_views),
    )
    if cull_poses is None or intrinsics is None:
        cull_poses = intrinsics = None
    return evaluate_reconstruction(rec_mesh, gt_mesh, config, cull_poses, intrinsics)
