"""``neb-slam eval`` on tiny run directories."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from neb_slam_core.cli.main import main
from neb_slam_core.geometry.se3 import make_pose
from neb_slam_core.io.trajectory import Trajectory, write_tum_trajectory
from neb_slam_core.types import Intrinsics


def write_run(run_dir, d=0.03):
    """Cube-corner ground truth; the estimate has noise d * sign(x y z) along z (ATE RMSE = d, see
    test_eval_trajectory_metrics) and lives in a rotated, shifted world frame."""
    corners = np.array([[x, y, z] for x in (-1.0, 1.0) for y in (-1.0, 1.0) for z in (-1.0, 1.0)])
    gt = np.tile(np.eye(4), (8, 1, 1))
    gt[:, :3, 3] = corners
    est = gt.copy()
    est[:, 2, 3] += d * np.prod(corners, axis=1)
    c, s = np.cos(0.4), np.sin(0.4)
    est = make_pose(np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]), [1.0, 2.0, 3.0]) @ est
    stamps = (1_000_000_000 + np.arange(8) * 100_000_000).astype(np.int64)
    run_dir.mkdir(parents=True, exist_ok=True)
    write_tum_trajectory(run_dir / "groundtruth.txt", Trajectory(stamps, gt))
    write_tum_trajectory(run_dir / "trajectory.txt", Trajectory(stamps + 3_000_000, est))  # 3 ms later
    return run_dir


def test_eval_run_dir_writes_metrics_and_plots(tmp_path, capsys):
    run = write_run(tmp_path / "run")
    (run / "metrics.json").write_text(json.dumps({"ms_per_frame_tracking": 12.5, "ate_rmse_cm": 99.0}))
    assert main(["eval", str(run)]) == 0
    metrics = json.loads((run / "metrics.json").read_text())
    # the file holds 8 decimals: 1e-8 m of rounding at most
    assert metrics["ate_rmse_cm"] == pytest.approx(3.0, abs=1e-5)
    assert metrics["ate_mean_cm"] == pytest.approx(3.0, abs=1e-5)
    assert metrics["n_poses"] == 8
    assert metrics["ms_per_frame_tracking"] == 12.5  # merged, not replaced
    assert metrics["rpe_trans_cm"] is None  # 0.7 s of poses: no pair 1 s apart
    assert metrics["rpe_frame_trans_cm"] > 0
    for name in ("trajectory.png", "ate_over_time.png"):
        assert (run / name).stat().st_size > 1000
    out = capsys.readouterr().out
    assert "ATE RMSE" in out and "3.000 cm" in out


def test_eval_two_files_directly(tmp_path, capsys):
    run = write_run(tmp_path / "run")
    assert main(["eval", "--est", str(run / "trajectory.txt"), "--gt", str(run / "groundtruth.txt")]) == 0
    assert "3.000 cm" in capsys.readouterr().out
    assert not (run / "metrics.json").exists()  # nothing written without a run dir or --out
    out = tmp_path / "results"
    assert (
        main(
            [
                "eval",
                "--est",
                str(run / "trajectory.txt"),
                "--gt",
                str(run / "groundtruth.txt"),
                "--out",
                str(out),
                "--no-plots",
            ]
        )
        == 0
    )
    assert json.loads((out / "metrics.json").read_text())["ate_rmse_cm"] == pytest.approx(3.0, abs=1e-5)
    assert not (out / "trajectory.png").exists()


def test_eval_reports_unmatched_files_clearly(tmp_path, capsys):
    run = write_run(tmp_path / "run")
    lines = (run / "trajectory.txt").read_text().splitlines()
    # shift the estimate's clock by 5 s: nothing associates
    shifted = [
        ln if ln.startswith("#") else f"{float(ln.split()[0]) + 5:.9f} " + " ".join(ln.split()[1:]) for ln in lines
    ]
    (run / "trajectory.txt").write_text("\n".join(shifted) + "\n")
    assert main(["eval", str(run)]) == 2
    err = capsys.readouterr().err
    assert "trajectory.txt" in err and "groundtruth.txt" in err and "only 0 of 8" in err
    assert main(["eval", str(tmp_path / "missing")]) == 2
    assert "run directory not found" in capsys.readouterr().err
    assert main(["eval"]) == 2
    assert "--est and --gt" in capsys.readouterr().err


def test_eval_skips_bad_ground_truth_lines_but_not_bad_estimate_lines(tmp_path, capsys, caplog):
    run = write_run(tmp_path / "run")
    gt_lines = (run / "groundtruth.txt").read_text().splitlines()
    data = [k for k, ln in enumerate(gt_lines) if not ln.startswith("#")]
    gt_lines[data[2]] = gt_lines[data[2]].rsplit(" ", 1)[0] + " nan"  # the third pose: not finite
    (run / "groundtruth.txt").write_text("\n".join(gt_lines) + "\n")
    assert main(["eval", str(run), "--no-plots"]) == 0
    assert json.loads((run / "metrics.json").read_text())["n_poses"] == 7
    assert any(f"skipped 1 bad line ({data[2] + 1};" in r.getMessage() for r in caplog.records)

    est_lines = (run / "trajectory.txt").read_text().splitlines()
    est_lines[data[4]] = est_lines[data[4]][:20]  # cut short, as by a crash while writing
    (run / "trajectory.txt").write_text("\n".join(est_lines) + "\n")
    capsys.readouterr()
    assert main(["eval", str(run), "--no-plots"]) == 2
    err = capsys.readouterr().err
    assert f"trajectory.txt: line {data[4] + 1}: expected 8 numbers" in err


def square(half: float, z: float) -> trimesh.Trimesh:
    v = np.array([[-half, -half, z], [half, -half, z], [half, half, z], [-half, half, z]], dtype=float)
    return trimesh.Trimesh(v, [[0, 1, 2], [0, 2, 3]], process=False)


def test_eval_with_meshes(tmp_path):
    run = write_run(tmp_path / "run")
    square(1.0, 4.01).export(run / "mesh.ply")
    # exact case: same triangulation moved 1 cm along the normal (see test_eval_recon)
    square(1.0, 4.0).export(tmp_path / "gt.ply")
    assert (
        main(
            [
                "eval",
                str(run),
                "--gt-mesh",
                str(tmp_path / "gt.ply"),
                "--n-points",
                "5000",
                "--depth-views",
                "0",
                "--no-cull",
                "--no-plots",
            ]
        )
        == 0
    )
    m = json.loads((run / "metrics.json").read_text())
    # PLY stores float32 vertices: 4.01 becomes 4.0100002 (2e-5 cm)
    assert m["accuracy_cm"] == pytest.approx(1.0, abs=1e-4)
    assert m["completion_cm"] == pytest.approx(1.0, abs=1e-4)
    assert m["completion_ratio_pct"] == 100.0
    assert m["depth_l1_cm"] is None and m["recon_culled"] is False
    assert m["ate_rmse_cm"] == pytest.approx(3.0, abs=1e-5)

    # culling: the ground truth also has a square behind every camera (they sit at the cube corners,
    # identity rotation, looking along +z; the square z = 4 is inside each one's view)
    trimesh.util.concatenate([square(1.0, 4.0), square(1.0, -5.0)]).export(tmp_path / "gt2.ply")
    intr = Intrinsics(32.0, 32.0, 31.5, 23.5, 64, 48)
    (run / "intrinsics.json").write_text(
        json.dumps(
            {"fx": intr.fx, "fy": intr.fy, "cx": intr.cx, "cy": intr.cy, "width": intr.width, "height": intr.height}
        )
    )
    common = [
        "eval",
        str(run),
        "--gt-mesh",
        str(tmp_path / "gt2.ply"),
        "--n-points",
        "20000",
        "--cull-stride",
        "1",
        "--no-plots",
    ]
    assert main(common + ["--depth-views", "0", "--no-cull"]) == 0
    whole = json.loads((run / "metrics.json").read_text())
    assert whole["completion_ratio_pct"] == pytest.approx(50.0, abs=1.5)
    assert main(common + ["--depth-views", "0"]) == 0
    culled = json.loads((run / "metrics.json").read_text())
    assert culled["recon_culled"] is True and culled["completion_ratio_pct"] == 100.0
    # at least the 1 cm shift; at most about what independent samples give: the visible half holds
    # 2500 points per m^2, d + erfcx(d sqrt(pi lam)) / (2 sqrt(lam)) = 1.47 cm (see test_eval_recon)
    assert 1.0 <= culled["accuracy_cm"] < 1.5

    assert main(["eval", str(run), "--gt-mesh", str(tmp_path / "nope.ply"), "--depth-views", "0"]) == 2
    assert (
        main(["eval", str(run), "--gt-mesh", str(tmp_path / "gt.ply"), "--intrinsics", str(tmp_path / "no.json")]) == 2
    )
