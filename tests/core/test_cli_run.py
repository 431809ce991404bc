"""``neb-slam run``: the offline run command and its run directory.

One end-to-end run on the ``small`` synthetic scene is shared by the file-content tests (module
fixture); the interruption and crash tests run a few frames on a tiny budget with ``Slam.process``
patched to fail at a chosen frame.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import logging
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

import neb_slam_core
from neb_slam_core.cli import run as run_cmd
from neb_slam_core.cli.main import main
from neb_slam_core.config_io import load_config
from neb_slam_core.datasets import open_dataset
from neb_slam_core.eval.plots import plot_block_allocation
from neb_slam_core.eval.trajectory_metrics import evaluate_ate
from neb_slam_core.io.run_dir import TIMINGS_COLUMNS, FrameLog, RunLog, read_timings
from neb_slam_core.io.trajectory import read_tum_trajectory
from neb_slam_core.scene.persistence import load_map
from neb_slam_core.slam import Slam
from neb_slam_core.types import Intrinsics, RgbdFrame

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
RUN_FILES = (
    "config.yaml",
    "intrinsics.json",
    "trajectory.txt",
    "groundtruth.txt",
    "timings.csv",
    "map.pt",
    "mesh.ply",
    "metrics.json",
    "trajectory.png",
    "ate_over_time.png",
    "blocks.png",
)
#: input frames of the shared run: --start 2 --stride 2 --frames 8
SHARED_INDICES = list(range(2, 18, 2))
#: a budget far below ci's for the interruption tests (they check files, not accuracy); with 3 first
#: iterations the map has no surface yet (no mesh), with 10 it has one
TINY = [
    "--set",
    "mapping.first_iterations=3",
    "tracking.iterations=2",
    "mapping.iterations=2",
    "--recon-points",
    "2000",
    "--depth-views",
    "0",
]


def run_cli(argv: list[str]) -> tuple[int, str]:
    """``neb-slam`` in-process; returns (exit code, stdout)."""
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        code = main(argv)
    return code, out.getvalue()


def _ci_args(out: Path, small_scene: Path, *more: str) -> list[str]:
    """``run`` on the small scene with config ci into ``out``, then ``more``."""
    return ["run", str(small_scene), "--config", "ci", "--out", str(out), *more]


def _shared_args(out: Path, small_scene: Path) -> list[str]:
    """The shared run's arguments, into ``out``."""
    return _ci_args(
        out,
        small_scene,
        "--start",
        "2",
        "--stride",
        "2",
        "--frames",
        str(len(SHARED_INDICES)),
        "--seed",
        "3",
        "--recon-points",
        "20000",
        "--depth-views",
        "10",
    )


@pytest.fixture(scope="module")
def shared_run(small_scene, tmp_path_factory):
    out = tmp_path_factory.mktemp("run") / "small"
    expected_cfg = load_config("ci", ["seed=3"])  # read now: the preset file may change while tests run
    code, stdout = run_cli(_shared_args(out, small_scene))
    return code, stdout, out, expected_cfg


def fail_at(monkeypatch, k: int, exc: BaseException) -> None:
    """Make ``Slam.process`` raise ``exc`` on the (k+1)-th frame it is given."""
    original = Slam.process

    def process(self, frame):
        if self.n_frames == k:
            raise exc
        return original(self, frame)

    monkeypatch.setattr(Slam, "process", process)


# ------------------------------------------------------------------------------------ the shared run


def test_run_writes_every_file_and_prints_the_run_dir_last(shared_run):
    code, stdout, out, _ = shared_run
    assert code == 0
    for name in RUN_FILES:
        assert (out / name).is_file(), name
    assert stdout.strip().splitlines()[-1] == str(out)
    assert "ATE RMSE" in stdout
    for name in ("trajectory.png", "ate_over_time.png", "blocks.png"):
        assert (out / name).read_bytes()[:8] == PNG_MAGIC


def test_trajectory_has_the_input_stamps_and_starts_at_the_ground_truth(shared_run, small_scene):
    _, _, out, _ = shared_run
    ds = open_dataset(small_scene)
    stamps = np.array([ds.stamps_ns[i] for i in SHARED_INDICES])
    est = read_tum_trajectory(out / "trajectory.txt")
    gt = read_tum_trajectory(out / "groundtruth.txt")
    np.testing.assert_array_equal(est.stamps_ns, stamps)
    np.testing.assert_array_equal(gt.stamps_ns, stamps)  # every synthetic frame has ground truth
    for k, i in enumerate(SHARED_INDICES):
        np.testing.assert_allclose(gt.poses[k], ds[i].T_world_cam, atol=1e-7)
    # the first pose is the first processed frame's ground truth (8 decimals in the file)
    np.testing.assert_allclose(est.poses[0], ds[SHARED_INDICES[0]].T_world_cam, atol=1e-7)


def test_metrics_match_the_files_they_summarise(shared_run):
    _, _, out, _ = shared_run
    m = json.loads((out / "metrics.json").read_text())
    for key in (
        "ate_rmse_cm",
        "n_blocks",
        "param_mb",
        "s_per_frame",
        "track_ms_mean",
        "map_ms_mean",
        "n_keyframes",
        "n_tracking_failures",
        "accuracy_cm",
        "completion_cm",
        "completion_ratio_pct",
        "depth_l1_cm",
    ):
        assert key in m, key
    assert m["status"] == "complete" and m["n_frames"] == len(SHARED_INDICES) and m["frames_unreadable"] == 0
    assert math.isfinite(m["ate_rmse_cm"])
    # the ATE is that of the written files (as `neb-slam eval` would compute it)
    ate = evaluate_ate(read_tum_trajectory(out / "trajectory.txt"), read_tum_trajectory(out / "groundtruth.txt"))
    assert m["ate_rmse_cm"] == pytest.approx(ate.rmse_cm, abs=1e-6)
    rows = read_timings(out / "timings.csv")
    assert [int(r["index"]) for r in rows] == SHARED_INDICES
    total = np.array([float(r["total_ms"]) for r in rows])
    assert m["s_per_frame"] == pytest.approx(total.mean() / 1e3, rel=1e-3)
    track = [float(r["track_ms"]) for r in rows[1:]]
    assert m["track_ms_mean"] == pytest.approx(np.mean(track), rel=1e-3)
    assert m["map_ms_mean"] == pytest.approx(np.mean([float(r["map_ms"]) for r in rows]), rel=1e-3)
    assert m["n_keyframes"] == sum(r["keyframe"] == "1" for r in rows)
    assert m["n_tracking_failures"] == sum(r["tracking_ok"] == "0" for r in rows)
    assert m["n_blocks"] == sum(r["new_block"] != "" for r in rows)
    loops = json.loads((out / "loops.json").read_text())
    assert m["n_loops_detected"] == len(loops) and m["n_loops_applied"] == sum(e["applied"] for e in loops)
    assert m["recon_culled"] is True  # culled to the ground-truth cameras
    assert all(math.isfinite(m[k]) for k in ("accuracy_cm", "completion_cm", "depth_l1_cm"))


def test_timings_csv_rows(shared_run, small_scene):
    _, _, out, _ = shared_run
    with (out / "timings.csv").open(newline="") as fh:
        header = next(csv.reader(fh))
    assert tuple(header) == TIMINGS_COLUMNS
    rows = read_timings(out / "timings.csv")
    ds = open_dataset(small_scene)
    assert [int(r["stamp_ns"]) for r in rows] == [int(ds.stamps_ns[i]) for i in SHARED_INDICES]
    first = rows[0]
    assert first["keyframe"] == "1" and first["new_block"] == "0" and float(first["track_ms"]) == 0.0
    for r in rows:
        parts = sum(float(r[c]) for c in ("track_ms", "allocate_ms", "map_ms", "loop_ms"))
        assert 0.0 <= parts <= float(r["total_ms"]) + 1e-3


def test_map_checkpoint_holds_the_keyframes(shared_run):
    _, _, out, _ = shared_run
    m = json.loads((out / "metrics.json").read_text())
    block_map, extra = load_map(out / "map.pt")
    assert len(block_map) == m["n_blocks"]
    assert block_map.param_mb() == pytest.approx(m["param_mb"])
    rows = read_timings(out / "timings.csv")
    assert extra["keyframe_frame_indices"] == [int(r["index"]) for r in rows if r["keyframe"] == "1"]
    assert extra["frame_indices"] == SHARED_INDICES
    poses = extra["keyframe_poses"].numpy()
    assert poses.shape == (m["n_keyframes"], 4, 4)
    # the first keyframe stays fixed: it is the first trajectory pose
    np.testing.assert_allclose(poses[0], read_tum_trajectory(out / "trajectory.txt").poses[0], atol=1e-7)


def test_config_mesh_and_intrinsics(shared_run, small_scene):
    _, _, out, expected_cfg = shared_run
    assert load_config(out / "config.yaml") == expected_cfg
    mesh = trimesh.load(out / "mesh.ply", force="mesh", process=False)
    assert len(mesh.faces) > 0 and np.isfinite(mesh.vertices).all()
    assert json.loads((out / "intrinsics.json").read_text()) == json.loads(
        (small_scene / "intrinsics.json").read_text()
    )


def test_map_continues_a_run_s_checkpoint(shared_run, small_scene, tmp_path, capsys):
    """--map: the shared run's map.pt is the starting map (its blocks are all in the new checkpoint,
    unchanged in place); a map file that is missing, or made with another block size, exits 2 naming it."""
    _, _, shared_out, _ = shared_run
    before, _ = load_map(shared_out / "map.pt")
    out = tmp_path / "continued"
    code, stdout = run_cli(
        [
            "run",
            str(small_scene),
            "--config",
            "ci",
            "--seed",
            "3",
            "--start",
            "18",
            "--frames",
            "2",
            "--map",
            str(shared_out / "map.pt"),
            "--out",
            str(out),
            "--no-mesh",
            *TINY,
        ]
    )
    assert code == 0 and stdout.strip().splitlines()[-1] == str(out)
    assert f"continuing {shared_out / 'map.pt'} ({len(before)} blocks)" in capsys.readouterr().err
    after, _ = load_map(out / "map.pt")
    assert len(after) >= len(before)
    for a, b in zip(before.blocks, after.blocks):
        assert torch.equal(a.centre, b.centre)
    missing = tmp_path / "no_map.pt"
    assert main(["run", str(small_scene), "--config", "ci", "--map", str(missing), "--out", str(tmp_path / "x")]) == 2
    assert str(missing) in capsys.readouterr().err
    assert (
        main(
            [
                "run",
                str(small_scene),
                "--config",
                "ci",
                "--set",
                "block.edge_m=2.0",
                "--map",
                str(shared_out / "map.pt"),
                "--out",
                str(tmp_path / "y"),
            ]
        )
        == 2
    )
    assert "block.edge_m" in capsys.readouterr().err
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()


# -------------------------------------------------------------------------------- interruptions


def test_ctrl_c_writes_the_frames_processed_so_far(small_scene, tmp_path, monkeypatch):
    fail_at(monkeypatch, 3, KeyboardInterrupt())
    out = tmp_path / "run"
    code, stdout = run_cli(_ci_args(out, small_scene, "--frames", "10", *TINY, "--set", "mapping.first_iterations=10"))
    assert code == 130
    est = read_tum_trajectory(out / "trajectory.txt")
    ds = open_dataset(small_scene)
    np.testing.assert_array_equal(est.stamps_ns, ds.stamps_ns[:3])
    m = json.loads((out / "metrics.json").read_text())
    assert m["status"] == "interrupted" and m["n_frames"] == 3 and math.isfinite(m["ate_rmse_cm"])
    for name in ("map.pt", "mesh.ply", "timings.csv", "blocks.png"):
        assert (out / name).is_file(), name
    assert len(read_timings(out / "timings.csv")) == 3
    assert stdout.strip().splitlines()[-1] == str(out)


def test_second_ctrl_c_aborts_the_writing(small_scene, tmp_path, monkeypatch, capsys):
    import neb_slam_core.mesh

    fail_at(monkeypatch, 2, KeyboardInterrupt())

    def interrupted_mesh(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(neb_slam_core.mesh, "extract_mesh", interrupted_mesh)
    out = tmp_path / "run"
    assert main(["run", str(small_scene), "--config", "ci", "--out", str(out), *TINY]) == 130
    assert "writing aborted" in capsys.readouterr().err
    assert len(read_tum_trajectory(out / "trajectory.txt")) == 2  # written before the mesh
    assert not (out / "mesh.ply").exists()


def test_sigterm_writes_the_frames_processed_so_far_and_exits_143(small_scene, tmp_path):
    # a real process and a real signal: the handler is installed by the command's entry point
    out = tmp_path / "run"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    package_parent = str(Path(neb_slam_core.__file__).resolve().parents[1])  # this checkout's code
    env["PYTHONPATH"] = os.pathsep.join(p for p in (package_parent, env.get("PYTHONPATH")) if p)
    cmd = [sys.executable, "-m", "neb_slam_core.cli.main", "run", str(small_scene), "--config", "ci"]
    cmd += ["--out", str(out), *TINY, "--set", "mapping.first_iterations=10"]
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    stderr: list[str] = []
    reader = threading.Thread(target=lambda: stderr.extend(iter(lambda: proc.stderr.read(1), "")), daemon=True)
    reader.start()
    try:
        deadline = time.monotonic() + 300
        # the progress bar's "N/60" counts processed frames
        while max((int(n) for n in re.findall(r"(\d+)/60 \[", "".join(stderr))), default=0) < 3:
            assert proc.poll() is None, "".join(stderr)
            assert time.monotonic() < deadline, "no progress: " + "".join(stderr)
            time.sleep(0.05)
        proc.send_signal(signal.SIGTERM)
        stdout = proc.stdout.read()
        code = proc.wait(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    reader.join(timeout=10)
    err = "".join(stderr)
    assert code == 143, err
    assert "interrupted by SIGTERM" in err and "Traceback" not in err, err
    m = json.loads((out / "metrics.json").read_text())
    n = m["n_frames"]
    assert m["status"] == "interrupted" and 3 <= n < 60, m
    est = read_tum_trajectory(out / "trajectory.txt")
    np.testing.assert_array_equal(est.stamps_ns, open_dataset(small_scene).stamps_ns[:n])
    for name in ("map.pt", "mesh.ply", "timings.csv", "trajectory.png", "blocks.png"):
        assert (out / name).is_file(), name
    block_map, extra = load_map(out / "map.pt")
    assert len(block_map) == m["n_blocks"] and extra["frame_indices"] == list(range(n))
    assert stdout.strip().splitlines()[-1] == str(out)


def test_engine_crash_writes_what_exists_then_reraises(small_scene, tmp_path, monkeypatch):
    fail_at(monkeypatch, 2, RuntimeError("boom"))
    out = tmp_path / "run"
    with pytest.raises(RuntimeError, match="boom"):
        run_cli(["run", str(small_scene), "--config", "ci", "--out", str(out), "--no-mesh", *TINY])
    assert len(read_tum_trajectory(out / "trajectory.txt")) == 2
    assert json.loads((out / "metrics.json").read_text())["status"] == "crashed"
    assert (out / "map.pt").is_file() and not (out / "mesh.ply").exists()


def _trajectory_text(run_dir: Path) -> list[str]:
    return [line for line in (run_dir / "trajectory.txt").read_text().splitlines() if not line.startswith("#")]


def test_resume_after_a_crash_continues_as_if_uninterrupted(shared_run, small_scene, tmp_path, monkeypatch):
    """A crash at the 7th frame leaves the checkpoint of the last keyframe; --resume goes on from it, and
    the poses of all frames equal the uninterrupted shared run's (the engine's state is whole in it)."""
    _, _, shared_out, _ = shared_run
    out = tmp_path / "crashed"
    fail_at(monkeypatch, 6, RuntimeError("boom"))
    with pytest.raises(RuntimeError, match="boom"):
        run_cli([*_shared_args(out, small_scene), "--checkpoint-every", "1"])
    monkeypatch.undo()
    assert json.loads((out / "metrics.json").read_text())["status"] == "crashed"
    assert (out / "checkpoint.pt").is_file()
    code, stdout = run_cli(["run", "--resume", str(out)])
    assert code == 0 and stdout.strip().splitlines()[-1] == str(out)
    assert _trajectory_text(out) == _trajectory_text(shared_out)
    m = json.loads((out / "metrics.json").read_text())
    assert m["status"] == "complete" and m["n_frames"] == len(SHARED_INDICES)
    assert len(read_timings(out / "timings.csv")) == len(SHARED_INDICES)
    assert not (out / "checkpoint.pt").exists()  # a completed run has nothing left to resume


def test_sigkill_leaves_a_checkpoint_to_resume(shared_run, small_scene, tmp_path):
    """A real SIGKILL as soon as a checkpoint exists: the file reads, and the resumed run ends with the
    uninterrupted run's poses."""
    _, _, shared_out, _ = shared_run
    out = tmp_path / "killed"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    package_parent = str(Path(neb_slam_core.__file__).resolve().parents[1])
    env["PYTHONPATH"] = os.pathsep.join(p for p in (package_parent, env.get("PYTHONPATH")) if p)
    cmd = [sys.executable, "-m", "neb_slam_core.cli.main", *_shared_args(out, small_scene), "--checkpoint-every", "1"]
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 300
        while not (out / "checkpoint.pt").is_file():
            assert proc.poll() is None and time.monotonic() < deadline, "no checkpoint before the run ended"
            time.sleep(0.02)
        proc.kill()
        proc.wait()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert not (out / "metrics.json").exists()  # killed: nothing written but the checkpoint
    code, _ = run_cli(["run", "--resume", str(out)])
    assert code == 0
    assert _trajectory_text(out) == _trajectory_text(shared_out)


def test_resume_refuses_other_options_and_a_missing_checkpoint(small_scene, tmp_path, capsys):
    assert main(["run", "--resume", str(tmp_path)]) == 2
    assert str(tmp_path / "checkpoint.pt") in capsys.readouterr().err
    assert main(["run", str(small_scene), "--resume", str(tmp_path), "--frames", "3"]) == 2
    assert "drop source, --frames" in capsys.readouterr().err
    assert main(["run", "--config", "ci"]) == 2
    assert "--resume RUN_DIR" in capsys.readouterr().err


# ------------------------------------------------------------------------------------- bad input


def test_unreadable_frame_is_skipped_with_one_warning_and_counted(small_scene, tmp_path, caplog):
    scene = tmp_path / "scene"
    shutil.copytree(small_scene, scene)
    depth_files = [ln.split()[1] for ln in (scene / "depth.txt").read_text().splitlines() if ln[:1] not in ("", "#")]
    cut = scene / depth_files[5]  # frame 5 of the 8 processed: a PNG cut short, as by a full disk
    cut.write_bytes(cut.read_bytes()[:100])
    out = tmp_path / "run"
    caplog.set_level(logging.WARNING)
    code, stdout = run_cli(
        ["run", str(scene), "--config", "ci", "--out", str(out), "--frames", "8", "--no-mesh", *TINY]
    )
    assert code == 0
    est = read_tum_trajectory(out / "trajectory.txt")
    np.testing.assert_array_equal(est.stamps_ns, open_dataset(scene).stamps_ns[[0, 1, 2, 3, 4, 6, 7]])
    m = json.loads((out / "metrics.json").read_text())
    assert m["status"] == "complete" and m["n_frames"] == 7 and m["frames_unreadable"] == 1
    warnings = [r.getMessage() for r in caplog.records if "could not be read" in r.getMessage()]
    assert len(warnings) == 1 and str(cut) in warnings[0] and "skipped 1 frame " in warnings[0], warnings
    assert "unreadable frames" in stdout and stdout.strip().splitlines()[-1] == str(out)


def test_no_readable_frame_exits_2(small_scene, tmp_path, capsys):
    scene = tmp_path / "scene"
    shutil.copytree(small_scene, scene)
    for png in (scene / "depth").iterdir():
        png.write_bytes(b"")
    out = tmp_path / "run"
    assert main(["run", str(scene), "--config", "ci", "--out", str(out), "--frames", "3"]) == 2
    assert "none of the 3 selected frames can be read" in capsys.readouterr().err
    assert not out.exists()


def test_missing_dataset_exits_2_naming_it(tmp_path, capsys):
    missing = tmp_path / "no_such_dataset"
    out = tmp_path / "run"
    assert main(["run", str(missing), "--out", str(out)]) == 2
    assert str(missing) in capsys.readouterr().err
    assert not out.exists()


def test_unknown_config_exits_2_naming_it(small_scene, tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["run", str(small_scene), "--config", "no_such_preset", "--out", str(out)]) == 2
    assert "no_such_preset" in capsys.readouterr().err
    assert main(["run", str(small_scene), "--set", "tracking.no_such_key=1", "--out", str(out)]) == 2
    assert "no_such_key" in capsys.readouterr().err
    assert not out.exists()


def test_bad_frame_selection_and_non_empty_out_exit_2(small_scene, tmp_path, capsys):
    assert main(["run", str(small_scene), "--start", "60", "--out", str(tmp_path / "a")]) == 2
    assert "--start 60" in capsys.readouterr().err
    assert main(["run", str(small_scene), "--stride", "0", "--out", str(tmp_path / "a")]) == 2
    assert "--stride" in capsys.readouterr().err
    busy = tmp_path / "busy"
    busy.mkdir()
    (busy / "keep.txt").write_text("x")
    assert main(["run", str(small_scene), "--config", "ci", "--out", str(busy)]) == 2
    err = capsys.readouterr().err
    assert str(busy) in err and "not empty" in err


# ------------------------------------------------------------------------------------ pieces


def test_frame_stamp_choices_are_the_loaders():
    import argparse

    from neb_slam_core.cli.run import add_arguments
    from neb_slam_core.datasets.base import FRAME_STAMPS

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    (action,) = [a for a in parser._actions if a.dest == "frame_stamp"]
    assert tuple(action.choices) == FRAME_STAMPS and action.default is None


def test_select_frames():
    assert list(run_cmd.select_frames(10)) == list(range(10))
    assert list(run_cmd.select_frames(10, start=3, stride=3)) == [3, 6, 9]
    assert list(run_cmd.select_frames(10, start=1, stride=2, frames=2)) == [1, 3]
    assert list(run_cmd.select_frames(10, frames=50)) == list(range(10))


def test_default_preset_follows_the_loader(small_scene, tmp_path):
    class FakeDataset:
        def __init__(self, name, root):
            self.name, self.root = name, root

    assert run_cmd.default_preset(FakeDataset("tum", small_scene)) == "synthetic"  # scene.json
    assert run_cmd.default_preset(FakeDataset("tum", tmp_path)) == "tum"
    assert run_cmd.default_preset(FakeDataset("scannet", tmp_path)) == "scannet"
    assert run_cmd.default_preset(FakeDataset("replica", tmp_path)) == "replica"
    assert run_cmd.default_preset(FakeDataset("seven_scenes", tmp_path)) == "base"
    assert run_cmd.default_preset(FakeDataset("bag", tmp_path / "x.mcap")) == "base"


def test_default_out_dir_is_named_by_dataset_and_time(tmp_path):
    src = tmp_path / "fr1_xyz"
    src.mkdir()
    now = time.strptime("2024-05-06 07:08:09", "%Y-%m-%d %H:%M:%S")
    first = run_cmd.default_out_dir(src, now, parent=tmp_path / "runs")
    assert first == tmp_path / "runs" / "fr1_xyz-20240506-070809"
    first.mkdir(parents=True)
    assert run_cmd.default_out_dir(src, now, parent=tmp_path / "runs").name == "fr1_xyz-20240506-070809-2"
    bag = tmp_path / "seq.mcap"
    bag.write_bytes(b"")
    assert run_cmd.default_out_dir(bag, now, parent=tmp_path / "runs").name == "seq-20240506-070809"


def test_run_log_ground_truth_skips_frames_without_pose():
    intr = Intrinsics(10.0, 10.0, 1.5, 1.5, 4, 4)
    run_log = RunLog()
    for i, has_gt in enumerate((True, False, True, True)):
        T = np.eye(4)
        T[0, 3] = i
        frame = RgbdFrame(
            np.zeros((4, 4, 3), np.uint8), np.ones((4, 4), np.float32), intr, 100 * i, T if has_gt else None, index=i
        )
        run_log.begin(frame)
    gt = run_log.groundtruth(3)
    np.testing.assert_array_equal(gt.stamps_ns, [0, 200])
    np.testing.assert_array_equal(gt.positions[:, 0], [0.0, 2.0])
    assert run_log.completed == [] and isinstance(run_log.frames[0], FrameLog)
    with pytest.raises(RuntimeError):
        RunLog().end(None)


def test_block_allocation_plot_draws_each_block_footprint():
    from matplotlib.patches import Rectangle

    traj = np.array([[0.0, 0.0, 0.0], [4.0, 0.1, 1.0], [8.0, 0.2, 3.0]])  # spreads most along x and z
    centres = np.array([[1.0, 0.0, 2.0], [6.0, 0.0, 2.5]])
    fig = plot_block_allocation(traj, centres, 5.0, np.array([0, 7]), traj[[0, 2]])
    ax = fig.axes[0]
    outlines = sorted((p for p in ax.patches if isinstance(p, Rectangle) and not p.get_fill()), key=lambda p: p.get_x())
    # footprints on the (x, z) plane: corner = centre - edge / 2, edge 5 m
    assert [(p.get_x(), p.get_y(), p.get_width(), p.get_height()) for p in outlines] == [
        (-1.5, -0.5, 5.0, 5.0),
        (3.5, 0.0, 5.0, 5.0),
    ]
    assert ax.get_xlabel() == "x [m]" and ax.get_ylabel() == "z [m]"
    # coloured by allocating frame: the colour bar spans frames 0..7 and the two outlines differ
    assert fig.axes[1].get_ylim() == (0.0, 7.0)
    assert outlines[0].get_edgecolor() != outlines[1].get_edgecolor()
    with pytest.raises(ValueError, match="one of each per block"):
        plot_block_allocation(traj, centres, 5.0, np.array([0]), traj[[0]])
