"""Evaluate a run: trajectory error (ATE, RPE) and, given meshes, reconstruction quality.

A run directory holds ``trajectory.txt`` (estimate) and ``groundtruth.txt`` (both TUM format:
``timestamp tx ty tz qx qy qz qw``), optionally ``mesh.ply`` (the reconstruction) and
``intrinsics.json`` (the camera, used to cull the meshes to what it saw). The command writes
``metrics.json`` into the run directory (merged into an existing one), ``trajectory.png`` and
``ate_over_time.png``, and prints a short table.

ATE: poses associated by stamp (nearest within --max-dt, each ground-truth pose used once), rigid
SE(3) alignment (no scale), RMSE of the translation residuals. RPE (``rpe_trans_cm``, ``rpe_rot_deg``):
RMSE over pose pairs --rpe-delta seconds apart; ``rpe_frame_*`` over consecutive matched poses.
Reconstruction (with --gt-mesh): accuracy, completion, completion ratio on sampled points (culled to
the ground-truth camera poses when the intrinsics are known), Depth L1 over random virtual views.
The reconstruction must be in the ground truth's world frame; --align-mesh maps it there with the ATE
alignment first.

Bad lines (not 8 numbers, non-finite, a quaternion that is not unit length): in the ground truth they
are skipped with one warning naming them, and the rest is evaluated; in the estimate the first one is
an error naming the file and the line (exit status 2).

Examples:
    neb-slam eval runs/fr1_xyz
    neb-slam eval runs/replica_room0 --gt-mesh data/replica/room0_mesh.ply
    neb-slam eval --est est.txt --gt groundtruth.txt --out results/
"""

from __future__ import annotations

import argparse
from pathlib import Path

HELP = "ATE / RPE and reconstruction metrics of a run, with plots"

METRICS_FILE = "metrics.json"
TRAJECTORY_FILE = "trajectory.txt"
GROUNDTRUTH_FILE = "groundtruth.txt"
MESH_FILE = "mesh.ply"
INTRINSICS_FILE = "intrinsics.json"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("run_dir", nargs="?", type=Path, help="run directory (trajectory.txt, groundtruth.txt, [mesh.ply])")
    p.add_argument("--est", type=Path, help="estimated trajectory (default: RUN_DIR/trajectory.txt)")
    p.add_argument("--gt", type=Path, help="ground-truth trajectory (default: RUN_DIR/groundtruth.txt)")
    p.add_argument(
        "--out",
        type=Path,
        help="where metrics.json and the plots go (default: RUN_DIR; without RUN_DIR and --out nothing is written)",
    )
    p.add_argument(
        "--max-dt", type=float, default=0.02, metavar="S", help="association window in seconds (default 0.02)"
    )
    p.add_argument("--no-align", action="store_true", help="ATE without the rigid alignment")
    p.add_argument(
        "--rpe-delta", type=float, default=1.0, metavar="S", help="RPE pair spacing in seconds (default 1.0)"
    )
    p.add_argument("--no-plots", action="store_true", help="do not write PNG figures")
    g = p.add_argument_group("reconstruction")
    g.add_argument("--gt-mesh", type=Path, help="ground-truth mesh; switches the reconstruction metrics on")
    g.add_argument("--mesh", type=Path, help="reconstructed mesh (default: RUN_DIR/mesh.ply)")
    g.add_argument(
        "--intrinsics", type=Path, help="camera intrinsics JSON for culling (default: RUN_DIR/intrinsics.json)"
    )
    g.add_argument("--no-cull", action="store_true", help="compare the whole meshes, no culling to the cameras' view")
    g.add_argument(
        "--cull-stride", type=int, default=5, metavar="K", help="cull with every K-th ground-truth pose (default 5)"
    )
    g.add_argument("--align-mesh", action="store_true", help="map the reconstruction by the ATE alignment first")
    g.add_argument("--n-points", type=int, default=200_000, help="points sampled per mesh (default 200000)")
    g.add_argument("--threshold-cm", type=float, default=5.0, help="completion-ratio threshold (default 5 cm)")
    g.add_argument("--depth-views", type=int, default=1000, help="virtual views for Depth L1, 0 to skip (default 1000)")
    g.add_argument("--seed", type=int, default=0, help="seed of the point and view sampling (default 0)")


def _resolve_paths(args: argparse.Namespace) -> tuple[Path, Path, Path | None]:
    from ..errors import DatasetError

    run_dir: Path | None = args.run_dir
    if run_dir is not None and not run_dir.is_dir():
        raise DatasetError(run_dir, "run directory not found")
    if run_dir is None and (args.est is None or args.gt is None):
        raise DatasetError(None, "give a run directory, or both --est and --gt")
    est = args.est or run_dir / TRAJECTORY_FILE
    gt = args.gt or run_dir / GROUNDTRUTH_FILE
    out = args.out or run_dir
    return est, gt, out


def _fmt(value: float | None, unit: str) -> str:
    return "n/a" if value is None else f"{value:.3f} {unit}"


def run(args: argparse.Namespace) -> int:
    from ..errors import DatasetError
    from ..eval.report import merge_metrics, recon_metrics, trajectory_metrics, write_trajectory_plots
    from ..io.trajectory import read_tum_trajectory

    est_path, gt_path, out_dir = _resolve_paths(args)
    est = read_tum_trajectory(est_path)  # an estimate is read whole: a bad line is an error naming it
    gt = read_tum_trajectory(gt_path, skip_bad_lines=True)  # bad ground-truth lines: skipped, one warning
    metrics, ate = trajectory_metrics(
        est,
        gt,
        max_dt_s=args.max_dt,
        align=not args.no_align,
        rpe_delta_s=args.rpe_delta,
        est_source=est_path,
        gt_source=gt_path,
    )
    rows = [
        ("matched poses", f"{ate.n_matched} of {ate.n_est} (ground truth {ate.n_gt})"),
        ("ATE RMSE", _fmt(ate.rmse_cm, "cm")),
        ("ATE mean / median / max", f"{ate.mean_cm:.3f} / {ate.median_cm:.3f} / {ate.max_cm:.3f} cm"),
        (
            f"RPE trans / rot ({args.rpe_delta:g} s)",
            f"{_fmt(metrics['rpe_trans_cm'], 'cm')} / {_fmt(metrics['rpe_rot_deg'], 'deg')}",
        ),
        (
            "RPE trans / rot (frame)",
            f"{_fmt(metrics['rpe_frame_trans_cm'], 'cm')} / {_fmt(metrics['rpe_frame_rot_deg'], 'deg')}",
        ),
    ]

    if args.gt_mesh is not None:
        rec_path = args.mesh or (args.run_dir / MESH_FILE if args.run_dir is not None else None)
        if rec_path is None:
            raise DatasetError(None, "--gt-mesh needs a reconstruction: give --mesh or a run directory with mesh.ply")
        recon = _evaluate_recon(args, rec_path, ate)
        metrics.update(recon_metrics(recon))
        rows += [
            ("accuracy", _fmt(recon.accuracy_cm, "cm")),
            ("completion", _fmt(recon.completion_cm, "cm")),
            (f"completion ratio (<{recon.completion_threshold_cm:g} cm)", _fmt(recon.completion_ratio_pct, "%")),
            (f"depth L1 ({recon.n_depth_views} views)", _fmt(recon.depth_l1_cm, "cm")),
            ("culled to the cameras' view", "yes" if recon.culled else "no"),
            (f"sampling floor ({recon.n_points} points)", _fmt(recon.sampling_floor_cm, "cm")),
        ]
    elif args.run_dir is not None and (args.run_dir / MESH_FILE).is_file():
        rows.append(("reconstruction", f"{MESH_FILE} found; pass --gt-mesh for accuracy / completion"))

    width = max(len(name) for name, _ in rows)
    print(f"estimate:     {est_path}\nground truth: {gt_path}")
    for name, value in rows:
        print(f"  {name:<{width}}  {value}")

    if out_dir is not None:
        merge_metrics(out_dir / METRICS_FILE, metrics)
        written = [out_dir / METRICS_FILE]
        if not args.no_plots:
            written += write_trajectory_plots(ate, out_dir)
        print("wrote " + ", ".join(str(p) for p in written))
    return 0


def _evaluate_recon(args: argparse.Namespace, rec_path: Path, ate):
    import logging

    from ..datasets.tum import read_intrinsics_json
    from ..errors import ConfigError, DatasetError
    from ..eval.report import evaluate_mesh_files

    if args.n_points < 1 or args.depth_views < 0 or args.cull_stride < 1 or not args.threshold_cm > 0:
        raise ConfigError("--n-points and --cull-stride must be >= 1, --depth-views >= 0, --threshold-cm > 0")
    poses = intrinsics = None
    if not args.no_cull:
        if args.intrinsics is not None and not args.intrinsics.is_file():
            raise DatasetError(
                args.intrinsics, "intrinsics file not found (expected JSON with fx, fy, cx, cy, width, height)"
            )
        intr_path = args.intrinsics or (args.run_dir / INTRINSICS_FILE if args.run_dir is not None else None)
        if intr_path is not None and intr_path.is_file():
            intrinsics = read_intrinsics_json(intr_path)
            poses = ate.gt_poses[:: args.cull_stride]
        else:
            logging.getLogger(__name__).warning(
                "no intrinsics (%s): reconstruction metrics are computed without culling", intr_path or "--intrinsics"
            )
    return evaluate_mesh_files(
        rec_path,
        args.gt_mesh,
        T_gt_rec=ate.T_gt_est if args.align_mesh else None,
        cull_poses=poses,
        intrinsics=intrinsics,
        n_points=args.n_points,
        threshold_cm=args.threshold_cm,
        depth_views=args.depth_views,
        seed=args.seed,
    )
